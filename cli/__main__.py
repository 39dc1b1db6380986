from trianflow_vo.cli.main import main

if __name__ == "__main__":
    main()
